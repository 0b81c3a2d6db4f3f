"""The core never names a protocol: every protocol question goes through the endpoint contract
(engine/endpoints/base.py), so adding one touches its package, one registry line, the
dependency list and the docs.

Counted outside engine/endpoints/: identifiers (names, attributes, functions, classes,
arguments), imports and string literals. Docstrings and comments may name a protocol (they
explain, they do not decide)."""

from __future__ import annotations

import ast
import re
from collections import Counter
from pathlib import Path

import pytest

from tests.support.repo import REPO

pytestmark = pytest.mark.fast  # no broker, no network peer, no ROS 2 node: ./scripts/test.sh's first tier

PROTOCOL_WORDS = {
    "mqtt": r"mqtt",
    "amqp": r"amqp",
    "ros2": r"ros2|rclpy|\bros\b|rosmsg",
    "mavlink": r"mavlink",
}
CEILINGS = {protocol: 0 for protocol in PROTOCOL_WORDS}
"""Before the endpoint contract answered every protocol question: AMQP 57, ROS 2 34, MAVLink
32, MQTT 7 (the MQTT package's first merge). A protocol the core must name again gets a
ceiling here with the reason, so the count can only go down."""


def _docstrings(tree: ast.AST) -> set[int]:
    return {
        id(node.value) for node in ast.walk(tree)
        if isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant) and isinstance(node.value.value, str)
    }


def _names(node: ast.AST, docstrings: set[int]) -> list[str]:
    if isinstance(node, ast.Name):
        return [node.id]
    if isinstance(node, ast.Attribute):
        return [node.attr]
    if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
        return [node.name]
    if isinstance(node, ast.arg):
        return [node.arg]
    if isinstance(node, ast.alias):
        return [node.name, node.asname or ""]
    if isinstance(node, ast.ImportFrom):
        return [node.module or ""]
    if isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in docstrings:
        return [node.value]
    return []


def protocol_names(root: Path = REPO / "engine") -> dict[str, list[str]]:
    """``protocol -> ["file:line: text", ...]`` of each place the core names it."""
    found: dict[str, list[str]] = {protocol: [] for protocol in PROTOCOL_WORDS}
    for path in sorted(root.rglob("*.py")):
        if "endpoints" in path.relative_to(root).parts:
            continue
        tree = ast.parse(path.read_text(encoding="utf-8"))
        docstrings = _docstrings(tree)
        for node in ast.walk(tree):
            for text in _names(node, docstrings):
                for protocol, pattern in PROTOCOL_WORDS.items():
                    if re.search(pattern, text, re.I):
                        found[protocol].append(f"{path.relative_to(root)}:{getattr(node, 'lineno', '?')}: {text[:60]!r}")
    return found


def test_the_core_names_no_protocol_beyond_its_ceiling():
    found = protocol_names()
    over = {protocol: places for protocol, places in found.items() if len(places) > CEILINGS[protocol]}
    assert not over, "\n".join(f"{protocol}: {len(places)} > {CEILINGS[protocol]}:\n  " + "\n  ".join(places)
                               for protocol, places in over.items())


def test_the_count_finds_what_it_must(tmp_path: Path):
    """An import, an identifier and a string literal count; a docstring and a comment do not."""
    (tmp_path / "core.py").write_text(
        '"""Talks MQTT."""\n'
        "import aiomqtt  # mqtt\n"
        "from engine.endpoints.mqtt import TRANSPORT\n"
        "mqtt_client = None\n"
        "PROTOCOL = 'mqtt'\n"
    )
    places = protocol_names(tmp_path)["mqtt"]
    assert Counter(place.split(":")[1] for place in places) == {"2": 1, "3": 1, "4": 1, "5": 1}, places
