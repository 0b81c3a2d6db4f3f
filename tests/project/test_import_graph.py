"""The engine's modules import one another without a cycle, and its groups one way.

Every module under engine/ is parsed with ``ast`` (nothing is imported) and every import is
an edge: at module level, under ``if TYPE_CHECKING:``, and inside functions. A cycle means
two modules that cannot be understood (or changed) one without the other, whether Python
happens to tolerate it at import time or not; specs and option values belong below the
behaviour that uses them. ``from a.b import c`` is an edge to ``a.b.c`` when that is a module
of the package, else to ``a.b``; a parent package's ``__init__`` is not counted as imported
(it is, by Python, but it declares nothing the child uses).

The groups of engine/, bottom to top (:data:`GROUPS`): the foundation (engine/common/), the
protocol packages (engine/endpoints/), the route language (engine/language/), the running
engine (engine/running/) and the operator's surface (engine/ops/). A module imports its own
group and the groups below it, never one above: the language is checked without starting
anything, the running engine runs what the language compiled, and nothing depends on the
command line. Every module belongs to a group: a new flat module in engine/ fails here.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from tests.support.repo import REPO

pytestmark = pytest.mark.fast  # no broker, no network peer, no ROS 2 node: ./scripts/test.sh's first tier

ENGINE = REPO / "engine"


def module_name(path: Path) -> str:
    parts = path.relative_to(ENGINE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def modules() -> dict[str, Path]:
    return {module_name(path): path for path in sorted(ENGINE.rglob("*.py"))}


def _absolute(node: ast.ImportFrom, importer: str, is_package: bool) -> str:
    if not node.level:
        return node.module or ""
    base = importer.split(".")
    base = base if is_package else base[:-1]
    base = base[: len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def imports(name: str, path: Path, known: set[str]) -> set[str]:
    """Engine modules that ``name`` imports anywhere in its source."""
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = _absolute(node, name, path.name == "__init__.py")
            targets = [f"{base}.{alias.name}" if f"{base}.{alias.name}" in known else base for alias in node.names]
        else:
            continue
        for target in targets:
            while target and target not in known:  # import a.b.c of a module a.b: the edge is to a.b
                target = target.rpartition(".")[0]
            if target and target != name:
                found.add(target)
    return found


def graph() -> dict[str, set[str]]:
    known = modules()
    names = set(known)
    return {name: imports(name, path, names) for name, path in known.items()}


def cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan), each sorted, and for
    each a concrete cycle through its first module so the failure shows the path."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    components: list[list[str]] = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for nxt in sorted(edges.get(node, ())):
            if nxt not in index:
                visit(nxt)
                low[node] = min(low[node], low[nxt])
            elif nxt in on_stack:
                low[node] = min(low[node], index[nxt])
        if low[node] == index[node]:
            component = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                component.append(member)
                if member == node:
                    break
            if len(component) > 1:
                components.append(sorted(component))

    for node in sorted(edges):
        if node not in index:
            visit(node)
    return sorted(components)


def a_cycle(edges: dict[str, set[str]], component: list[str]) -> list[str]:
    """One concrete cycle inside ``component``, from its first module back to it (BFS)."""
    members, start = set(component), component[0]
    previous: dict[str, str] = {}
    frontier = [start]
    while frontier:
        nxt_frontier = []
        for node in frontier:
            for nxt in sorted(edges[node] & members):
                if nxt == start:
                    path = [node]
                    while path[-1] != start:
                        path.append(previous[path[-1]])
                    return [start, *reversed(path[:-1]), start] if node != start else [start, start]
                if nxt not in previous:
                    previous[nxt] = node
                    nxt_frontier.append(nxt)
        frontier = nxt_frontier
    return component


def describe(edges: dict[str, set[str]]) -> list[str]:
    return [" -> ".join(a_cycle(edges, component)) + f"  (component: {', '.join(component)})"
            for component in cycles(edges)]


def test_the_graph_sees_every_kind_of_import():
    edges = graph()
    assert "engine.running.runtime" in edges and "engine.endpoints.mavlink.connection" in edges
    assert "engine.endpoints.base" in edges["engine.running.runtime"] or any(
        "engine.endpoints" in target for target in edges["engine.running.runtime"])
    found = cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}})
    assert found == [["a", "b", "c"]]
    assert a_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}, ["a", "b", "c"]) == ["a", "b", "c", "a"]


def test_function_level_and_type_checking_imports_are_edges(tmp_path: Path):
    source = (  # a made-up package "pkg", so no rename of the engine's modules touches it
        "from typing import TYPE_CHECKING\n"
        "if TYPE_CHECKING:\n    from pkg.runtime import Engine\n"
        "def f():\n    from pkg import plan\n    import pkg.routes\n"
        "from . import pipeline\n"
    )
    path = tmp_path / "x.py"
    path.write_text(source)
    known = {"pkg.runtime", "pkg.plan", "pkg.routes", "pkg.pipeline", "pkg.x"}
    assert imports("pkg.x", path, known) == {"pkg.runtime", "pkg.plan", "pkg.routes", "pkg.pipeline"}


def test_engine_modules_import_without_a_cycle():
    problems = describe(graph())
    assert not problems, "import cycles among engine/ modules:\n" + "\n".join(problems)


GROUPS = ("engine.common", "engine.endpoints", "engine.language", "engine.running", "engine.ops")
"""The groups of engine/, bottom to top (see the module docstring)."""
TOP_LEVEL = {"engine": "engine.common", "engine.__main__": "engine.ops"}
"""The package itself (its version) sits with the foundation; ``python -m engine`` with the CLI."""
UPWARD_ALLOWED: set[tuple[str, str]] = set()
"""Known imports against the direction, each to go (none left: the two sources that built
their fair inbox with ``fairness.route_inbox`` ask their route, ``Deliver.inbox``). Nothing
may be added; a stale entry fails."""


def group_of(module: str) -> str | None:
    if module in TOP_LEVEL:
        return TOP_LEVEL[module]
    return next((group for group in GROUPS if module == group or module.startswith(group + ".")), None)


def upward(edges: dict[str, set[str]]) -> list[tuple[str, str]]:
    """Imports from a lower group into a higher one, ``(importer, imported)``."""
    rank = {group: index for index, group in enumerate(GROUPS)}
    found = []
    for importer, targets in edges.items():
        for target in targets:
            low, high = group_of(importer), group_of(target)
            if low is not None and high is not None and rank[low] < rank[high]:
                found.append((importer, target))
    return sorted(found)


def test_every_module_belongs_to_a_group():
    loose = sorted(name for name in modules() if group_of(name) is None)
    assert not loose, f"modules outside the groups {GROUPS} (move each into the group it belongs to): {loose}"


def test_the_groups_import_one_way():
    found = set(upward(graph()))
    against = sorted(found - UPWARD_ALLOWED)
    assert not against, ("imports from a lower group into a higher one (bottom to top: " + ", ".join(GROUPS) + "); move "
                         "the declaration the lower module needs down instead:\n"
                         + "\n".join(f"  {importer} -> {target}" for importer, target in against))
    stale = sorted(UPWARD_ALLOWED - found)
    assert not stale, f"UPWARD_ALLOWED lists imports that are gone; remove them: {stale}"


def test_the_direction_check_finds_an_upward_import():
    edges = {"engine.common.options": {"engine.language.routes"}, "engine.ops.cli": {"engine.running.runtime"},
             "engine.language.routes": {"engine.endpoints.base", "engine.common.options"}, "engine.__main__": {"engine.ops.cli"}}
    assert upward(edges) == [("engine.common.options", "engine.language.routes")]


def test_the_core_reaches_a_protocol_only_through_the_registry():
    """Outside engine/endpoints/ a protocol package is never imported: only the registry
    (engine/endpoints/__init__.py) and the contract (engine/endpoints/base.py)."""
    contract = {"engine.endpoints", "engine.endpoints.base"}
    found = sorted((importer, target) for importer, targets in graph().items() if group_of(importer) != "engine.endpoints"
                   for target in targets if group_of(target) == "engine.endpoints" and target not in contract)
    assert not found, f"the core imports a protocol package: {found}"


ENGINE_POLICIES = ("fairness", "throttle")
"""Core modules of the route's delivery policy: a route's ``fair:`` and ``throttle:`` are the
engine's to apply; a source asks its route for its queue (``Deliver.inbox``) and runs the
engine's read loop (engine/endpoints/pump.py), and never decides them itself."""


def test_endpoints_leave_fairness_and_throttle_to_the_engine():
    edges = graph()
    found = sorted(f"{name} -> {target}" for name, targets in edges.items() if name.startswith("engine.endpoints.")
                   for target in targets
                   if not target.startswith("engine.endpoints.") and target.rpartition(".")[2] in ENGINE_POLICIES)
    assert not found, "endpoints importing the engine's fairness or throttle:\n" + "\n".join(found)


if __name__ == "__main__":  # python -m tests.project.test_import_graph: print the cycles
    print("\n".join(describe(graph())) or "no cycle")
    print("\n".join(f"{importer} -> {target}" for importer, target in upward(graph())) or "no upward import")
