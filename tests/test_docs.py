"""The documentation cannot rot: its function examples run, its schemas and tutorial are real."""

from __future__ import annotations

import json
import re
import subprocess
import sys

import pytest

from engine.mapping import compile_mapping, known_functions
from engine.schemas import SchemaError, SchemaRegistry
from tests.conftest import REPO

DOCS = REPO / "docs"
ROW = re.compile(r"^\| `(?P<name>\w+)` \| `` (?P<expr>.+?) `` \| `(?P<result>.+?)` \| .* \|$")


def test_every_function_is_documented_with_an_example_that_holds():
    text = (DOCS / "route-language.md").read_text()
    source = json.loads(text.split("## Functions", 1)[1].split("```json", 1)[1].split("```", 1)[0])
    rows = [ROW.match(line) for line in text.splitlines() if line.startswith("| `")]
    examples = {m["name"]: (m["expr"].replace("\\|", "|"), m["result"]) for m in rows if m and "(" in m["expr"]}
    assert sorted(examples) == known_functions()
    for name, (expression, result) in examples.items():
        value = compile_mapping(expression)(source)
        if result.startswith("<"):
            assert type(value).__name__ == {"<number>": "float", "<object>": "dict", "<string>": "str"}[result], name
        else:
            assert value == json.loads(result), f"{name}: {expression} gives {value!r}, the docs say {result}"


def test_every_schema_is_documented():
    text = (DOCS / "schemas.md").read_text()
    for name in SchemaRegistry(REPO / "schemas").names():
        if ".v" in name:
            assert f"({name})" in text, name


def test_the_tutorial_route_and_its_test_are_the_files_it_shows():
    tutorial = (DOCS / "tutorial.md").read_text()
    for name in ("tractor.yaml", "tractor.test.yaml"):
        assert (DOCS / "tutorial" / "routes" / name).read_text() in tutorial, name
    result = subprocess.run([sys.executable, "-m", "engine", "test", "--routes", "docs/tutorial/routes", "--schemas", "schemas"],
                            capture_output=True, text=True, cwd=REPO, timeout=60)
    assert result.returncode == 0, result.stdout + result.stderr
    assert result.stdout.splitlines()[-1] == "2 passed, 0 failed"
    assert "[docs/](docs/README.md)" in (REPO / "README.md").read_text()


def _anchors(text: str) -> set[str]:
    """GitHub's heading anchors (lowercase, punctuation dropped, spaces to hyphens) and explicit ids."""
    slugs = {re.sub(r"[^a-z0-9 _-]", "", line.lstrip("#").strip().lower()).replace(" ", "-")
             for line in text.splitlines() if line.startswith("#")}
    return slugs | set(re.findall(r'<a id="([^"]+)"></a>', text))


def test_links_between_the_docs_resolve():
    """Every relative link of README.md and docs/*.md names a file that exists and, with a
    #fragment, a heading or anchor it has (route-language.md links into route-keys.md)."""
    broken = []
    for page in [REPO / "README.md", *sorted(DOCS.glob("*.md"))]:
        for target, fragment in re.findall(r"\]\(((?!https?:)[^)#\s]*)(?:#([^)\s]+))?\)", page.read_text()):
            linked = (page.parent / target).resolve() if target else page
            if not linked.exists() or (fragment and linked.suffix == ".md" and fragment not in _anchors(linked.read_text())):
                broken.append(f"{page.relative_to(REPO)}: {target}#{fragment}")
    assert broken == []
    assert "(route-keys.md)" in (DOCS / "route-language.md").read_text()


def test_the_shared_types_are_defined_and_the_stamp_is_what_the_schemas_accept():
    """schemas.md defines every shared type of envelope.v1.json that the tables name, and what
    it says a stamp is (and is not) is what validation does."""
    text = (DOCS / "schemas.md").read_text()
    shared = json.loads((REPO / "schemas" / "envelope.v1.json").read_text())["$defs"]
    for name in set(shared) - {"header"}:
        assert f"### `{name}`" in text, name
    position = SchemaRegistry(REPO / "schemas").get("position")
    fix = {"agent_id": "uav1", "lat": -22.0, "lon": -47.9}
    position.validate({**fix, "stamp": {"sec": 1700000000, "nanosec": 500000000}})
    stamp_section = text.split("### `stamp`", 1)[1].split("###", 1)[0]
    for refused, shown in ((1700000000.5, "`1700000000.5`"), ("2023-11-14T22:13:20Z", "ISO 8601"), ({"sec": 1700000000}, "`{sec}` without")):
        assert shown in stamp_section
        with pytest.raises(SchemaError):
            position.validate({**fix, "stamp": refused})
    assert "UNIX seconds" not in text.split("| `stamp` |", 1)[1].split("\n", 1)[0]
