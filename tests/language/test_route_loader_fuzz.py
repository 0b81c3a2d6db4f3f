"""Hostile route files, measured (issue 21): the loader behind ``check`` and ``run`` answers
every malformed file, YAML, JMESPath mapping or template with ``file:line: message``
problems, never a traceback or a hang.

Inputs are a valid route file damaged by hypothesis (characters inserted, deleted or
replaced anywhere) and valid files whose mapping, routing key, topic, ``format()`` template,
``${...}`` reference and option values are arbitrary text. Each input runs in-process with a
per-input time limit (HANG_S). Each fuzz asserts it reached both outcomes (some inputs still
load, others are refused), so a strategy that stopped producing one would fail instead of passing
vacuously; the counts print with ``-s``."""

from __future__ import annotations

import re
import tempfile
import time
from collections import Counter
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
ALPHABET = st.sampled_from(list("{}[]()'\"`:@,.|&!?*$#-_ \n\tabxyz019") + ["__class__", "${", "${file:", "format(", "\\u0000", "\t- "])


def _load(tmp_path: Path, text: str, outcomes: Counter[str]) -> None:
    """Load ``text`` as a route file: it loads, or every problem names ``r.yaml:LINE``; counted
    in ``outcomes`` (valid, invalid, and the slowest load in ms)."""
    directory = Path(tempfile.mkdtemp(dir=tmp_path))
    (directory / "r.yaml").write_text(text)
    began = time.monotonic()
    try:
        load_routes(directory, SCHEMAS, env={})
        outcomes["valid"] += 1
    except RoutesInvalid as invalid:
        outcomes["invalid"] += 1
        assert invalid.problems, text
        for problem in invalid.problems:
            assert PROBLEM.match(str(problem).removeprefix(f"{directory}/")), (str(problem), text)
    took = time.monotonic() - began
    outcomes["slowest_ms"] = max(outcomes["slowest_ms"], round(took * 1000))
    assert took < HANG_S, f"{took:.1f}s for one file: {text!r}"


def _reached_both_outcomes(name: str, outcomes: Counter[str]) -> None:
    print(f"\n{name}: {outcomes['valid'] + outcomes['invalid']} inputs, {outcomes['valid']} valid, "
          f"{outcomes['invalid']} invalid (each with file:line problems), 0 tracebacks, slowest {outcomes['slowest_ms']} ms")
    assert outcomes["valid"] > 0 and outcomes["invalid"] > 0, f"{name}: the fuzz reached one outcome only: {dict(outcomes)}"


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


def test_a_damaged_route_file_gets_file_line_problems(tmp_path: Path) -> None:
    outcomes: Counter[str] = Counter()

    @FUZZ
    @given(damaged())
    def load(text: str) -> None:
        _load(tmp_path, text, outcomes)

    load()
    _reached_both_outcomes("damaged route files", outcomes)


def test_arbitrary_mappings_and_templates_get_file_line_problems(tmp_path: Path) -> None:
    outcomes: Counter[str] = Counter()

    @FUZZ
    @given(st.lists(ALPHABET, max_size=12).map("".join), st.lists(ALPHABET, max_size=12).map("".join),
           st.lists(ALPHABET, max_size=8).map("".join))
    def load(mapping: str, key: str, topic: str) -> None:
        _load(tmp_path, TEMPLATE.format(mapping=_quoted(mapping), key=_quoted(key), topic=_quoted("/" + topic)), outcomes)

    load()
    _reached_both_outcomes("arbitrary mappings and templates", outcomes)


def test_an_amqp_url_that_is_not_a_url_is_a_problem_with_its_password_hidden(tmp_path: Path) -> None:
    """Found by the damaged-file fuzz: ``amqp://[farmer:...`` (an unbalanced ``[``) made
    urllib raise while the problem's own text was redacted: a traceback instead of a problem."""
    (tmp_path / "r.yaml").write_text(VALID.replace("amqp://farmer:${RABBITROS_FUZZ_PW:-pw}@", "amqp://[farmer:secret@"))
    with pytest.raises(RoutesInvalid) as refused:
        load_routes(tmp_path, SCHEMAS, env={})
    problems = [str(problem) for problem in refused.value.problems]
    assert any("is not a valid URL" in problem and "amqp://[farmer:***@localhost" in problem for problem in problems), problems
    assert not any("secret" in problem for problem in problems), problems
