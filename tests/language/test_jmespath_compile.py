"""Compiled JMESPath (engine.language.jmespath_compile) gives exactly jmespath's results.

Hypothesis generates expressions of every form the compiler handles (field paths,
subexpressions, index/slice, projections, flatten, filters, multiselect hashes and lists,
comparisons, and/or/not, pipes, literals, function calls with expression references) and
documents over the same field names, and compares the compiled closure with jmespath's
interpreter: equal results (same types), or the same exception type. Every mapping the
project ships (routes/, examples/) is compared the same way on generated messages.
"""

from __future__ import annotations

import json
from typing import Any, Iterator

import jmespath
import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from jmespath import functions

from engine.language.jmespath_compile import compile_parsed, is_compiled
from engine.language.mapping import FieldFunctions, compile_mapping
from tests.support.repo import REPO

pytestmark = pytest.mark.fast  # no broker, no network peer, no ROS 2 node: ./scripts/test.sh's first tier

NAMES = ["a", "b", "c", "n", "s"]


class DeterministicFunctions(FieldFunctions):
    """The engine's functions with a fixed clock and ids, so two evaluations can be compared."""

    @functions.signature()
    def _func_now(self) -> float:
        return 1732320000.5

    @functions.signature()
    def _func_stamp(self) -> dict[str, int]:
        return {"sec": 1732320000, "nanosec": 500000000}

    @functions.signature()
    def _func_uuid(self) -> str:
        return "00000000000000000000000000000000"

    @functions.signature({"types": ["number"]})
    def _func_stamp_boot_ms(self, time_boot_ms: int) -> dict[str, int]:
        return {"sec": 1732320000, "nanosec": int(time_boot_ms) % 1000 * 1_000_000}

    @functions.signature({"types": ["number"]})
    def _func_stamp_usec(self, time_usec: int) -> dict[str, int]:
        return {"sec": 1732320000, "nanosec": int(time_usec) % 1_000_000 * 1000}


OPTIONS = jmespath.Options(custom_functions=DeterministicFunctions())


def outcome(evaluate: Any, data: Any) -> tuple[str, str]:
    try:
        return "ok", repr(evaluate(data))
    except Exception as exc:  # the same exception type, whatever it is
        return "raised", type(exc).__name__


def assert_same(expression: str, data: Any) -> None:
    parsed = jmespath.compile(expression)
    expected = outcome(lambda d: parsed.search(d, options=OPTIONS), data)
    assert outcome(compile_parsed(parsed, OPTIONS), data) == expected, (expression, data)


# ---------------------------------------------------------------- generated expressions

identifiers = st.sampled_from(NAMES) | st.just('"quoted key"')
scalars = (
    st.none() | st.booleans() | st.integers(-3, 3) | st.integers() | st.floats(allow_nan=False, allow_infinity=False)
    | st.text(alphabet="ab é", max_size=3) | st.sampled_from([{}, [], "", 0, 1, 0.0, False, True])
)
literal_json = scalars.map(lambda v: "`" + json.dumps(v).replace("`", "\\`") + "`")
raw_strings = st.text(alphabet="abc é", max_size=3).map(lambda s: f"'{s}'")
paths = st.lists(identifiers, min_size=1, max_size=4).map(".".join)
leaves = paths | st.just("@") | literal_json | raw_strings
FUNCTIONS_1 = ["length", "abs", "to_string", "to_number", "type", "keys", "values", "not_null", "to_array",
               "sum", "max", "min", "reverse", "sort", "floor", "ceil", "avg", "round", "to_int", "mm_to_m"]
FUNCTIONS_2 = ["not_null", "contains", "starts_with", "join", "default", "add", "mul", "div", "sub", "merge"]


def composite(children: st.SearchStrategy[str]) -> st.SearchStrategy[str]:
    two = st.tuples(children, children)
    return st.one_of(
        st.tuples(children, identifiers).map(lambda t: f"({t[0]}).{t[1]}"),
        st.tuples(children, st.integers(-3, 3)).map(lambda t: f"({t[0]})[{t[1]}]"),
        st.tuples(children, st.sampled_from(["", "1", "-1"]), st.sampled_from(["", "2", "-2"]),
                  st.sampled_from(["", "1", "2", "-1"])).map(lambda t: f"({t[0]})[{t[1]}:{t[2]}:{t[3]}]"),
        st.tuples(paths, st.sampled_from(["[*]", ".*", "[]"]), paths).map(lambda t: f"{t[0]}{t[1]}.{t[2]}"),
        st.tuples(children, st.sampled_from(["[*]", ".*", "[]"])).map(lambda t: f"({t[0]}){t[1]}"),
        st.tuples(paths, children, children).map(lambda t: f"{t[0]}[?{t[1]}].{{x: {t[2]}}}"),
        st.tuples(children, children).map(lambda t: f"({t[0]})[?{t[1]}]"),
        st.tuples(paths, children, children).map(lambda t: f"{t[0]}[*].{{k: {t[1]}, \"v w\": {t[2]}}}"),
        st.lists(st.tuples(identifiers, children), min_size=1, max_size=3).map(
            lambda pairs: "{" + ", ".join(f"{k}: {v}" for k, v in pairs) + "}"),
        st.lists(children, min_size=1, max_size=3).map(lambda items: "[" + ", ".join(items) + "]"),
        st.tuples(children, st.sampled_from(["==", "!=", "<", "<=", ">", ">="]), children).map(
            lambda t: f"({t[0]}) {t[1]} ({t[2]})"),
        two.map(lambda t: f"({t[0]}) && ({t[1]})"),
        two.map(lambda t: f"({t[0]}) || ({t[1]})"),
        children.map(lambda c: f"!({c})"),
        two.map(lambda t: f"({t[0]}) | ({t[1]})"),
        st.tuples(st.sampled_from(FUNCTIONS_1), children).map(lambda t: f"{t[0]}({t[1]})"),
        st.tuples(st.sampled_from(FUNCTIONS_2), children, children).map(lambda t: f"{t[0]}({t[1]}, {t[2]})"),
        st.tuples(st.sampled_from(["sort_by", "max_by", "min_by", "map"]), children, identifiers).map(
            lambda t: f"{t[0]}(({t[1]}), &{t[2]})" if t[0] != "map" else f"map(&{t[2]}, ({t[1]}))"),
    )


expressions = st.recursive(leaves, composite, max_leaves=8)
values = st.recursive(
    scalars,
    lambda children: st.lists(children, max_size=4)
    | st.dictionaries(st.sampled_from(NAMES + ["quoted key"]), children, max_size=5),
    max_leaves=25,
)
documents = st.fixed_dictionaries({name: values for name in NAMES}) | values
"""Mostly objects holding every generated name, so paths lead somewhere."""


@settings(max_examples=700, deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much])
@given(expressions, documents)
def test_generated_expressions_evaluate_as_jmespath_does(expression: str, data: Any) -> None:
    try:
        parsed = jmespath.compile(expression)
    except jmespath.exceptions.JMESPathError:
        return  # generated text that is not an expression: nothing to compare
    assert is_compiled(parsed), expression
    assert_same(expression, data)


@pytest.mark.parametrize(
    "expression, data",
    [
        ("a.b.c", {"a": {"b": {"c": 1}}}), ("a.b.c", {"a": [1]}), ("a.b.c", {"a": {"b": "text"}}),
        ("a[0].b", {"a": [{"b": 2}]}), ("a[-1]", {"a": [1, 2]}), ("a[5]", {"a": [1]}), ("a[::-1]", {"a": [1, 2, 3]}),
        ("a[*].b", {"a": [{"b": 1}, {"c": 2}, {"b": None}, 3]}), ("a.*.b", {"a": {"x": {"b": 1}, "y": 2}}),
        ("a[]", {"a": [[1], 2, [3, [4]]]}), ("a[*]", {"a": [1, None, 2]}), ("a.*", {"a": {"x": None, "y": 1}}),
        ("a[]", {"a": [None, [None]]}), ("a[?b]", {"a": [{"b": {}}, {"b": [0]}, None]}), ("a[?b > `1`].c", {"a": [{"b": 2, "c": "x"}, {"b": "2"}, {"b": True}]}),
        ("{x: a, y: b.c}", None), ("[a, b]", None), ("!`0`", {}), ("!a", {"a": []}), ("a == `1`", {"a": True}),
        ("a != `0`", {"a": False}), ("a < b", {"a": "a", "b": "b"}), ("a < b", {"a": 1, "b": "b"}),
        ("a || b", {"a": {}, "b": 0}), ("a && b", {"a": "", "b": 1}), ("sort_by(a, &b)", {"a": [{"b": 2}, {"b": 1}]}),
        ("max_by(a, &b)", {"a": [{"b": "x"}, {"b": 1}]}), ("length(a)", {"a": 3}), ("nope(a)", {"a": 1}),
        ("div(a, `0`)", {"a": 1}), ("format('{x}', @)", {"y": 1}), ("`[1, 2]`", None), ("@", [1]),
    ],
)
def test_edge_cases_evaluate_as_jmespath_does(expression: str, data: Any) -> None:
    assert_same(expression, data)


# ---------------------------------------------------------------- the shipped mappings

def shipped_mappings() -> Iterator[tuple[str, str]]:
    for path in sorted([*REPO.glob("routes/**/*.yaml"), *REPO.glob("examples/**/*.yaml")]):
        document = yaml.safe_load(path.read_text()) or {}
        for route in document.get("routes") or []:
            for where, expression in (("mapping", route.get("mapping")), ("sink.mapping", (route.get("sink") or {}).get("mapping"))):
                if isinstance(expression, str):
                    yield f"{path.relative_to(REPO)}:{route.get('name')}:{where}", expression


SHIPPED = list(shipped_mappings())


def field_names(node: dict[str, Any]) -> set[str]:
    names = {node["value"]} if node["type"] == "field" else set()
    for child in node.get("children", ()):
        if isinstance(child, dict):
            names |= field_names(child)
    return names


def test_the_project_ships_mappings() -> None:
    assert len(SHIPPED) >= 5, SHIPPED


@pytest.mark.parametrize("where, expression", SHIPPED, ids=[where for where, _ in SHIPPED])
def test_shipped_mapping_evaluates_as_jmespath_does(where: str, expression: str) -> None:
    parsed = jmespath.compile(expression)
    assert is_compiled(parsed)
    names = sorted(field_names(parsed.parsed))
    values = (
        st.integers(-(2**31), 2**31) | st.sampled_from([-1, 0, 1, 2, 65535]) | st.floats(-1e3, 1e3)
        | st.text(max_size=4) | st.none() | st.lists(st.integers(-5, 5), max_size=3)
        | st.lists(st.fixed_dictionaries({}, optional={n: st.integers(-5, 5) | st.floats(-90, 90) for n in names}), max_size=3)
    )
    messages = st.fixed_dictionaries({}, optional={name: values for name in names})

    # 40 messages a mapping: the 45 shipped ones took 37 s of the fast tier's CPU at 100 (the VDA 5050
    # state mappings 3-4 s each), and the generated expressions below cover the forms in depth
    @settings(max_examples=40, deadline=None)
    @given(messages)
    def compare(message: dict[str, Any]) -> None:
        assert_same(expression, message)

    compare()


def test_compile_mapping_does_not_interpret(monkeypatch: pytest.MonkeyPatch) -> None:
    """The engine's mappings run compiled: jmespath's interpreter is never entered per message."""
    expression = next(e for w, e in SHIPPED if "uav-weeds" in w)
    message = {"agent": "uav1", "id": "x", "stamp": 1.0, "detections": [{"lat": 1.0, "lon": 2.0, "confidence": 0.5}] * 3}
    expected = jmespath.compile(expression).search(message, options=OPTIONS)
    mapper = compile_mapping(expression)

    def interpreted(*args: Any, **kwargs: Any) -> Any:
        raise AssertionError("jmespath's interpreter was used")

    monkeypatch.setattr(jmespath.visitor.TreeInterpreter, "visit", interpreted)
    assert mapper is not None and mapper(message) == expected
