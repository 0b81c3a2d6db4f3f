"""The engine's modules import one another without a cycle.

Every module under engine/ is parsed with ``ast`` (nothing is imported) and every import is
an edge: at module level, under ``if TYPE_CHECKING:``, and inside functions. A cycle means
two modules that cannot be understood (or changed) one without the other, whether Python
happens to tolerate it at import time or not; specs and option values belong below the
behaviour that uses them. ``from a.b import c`` is an edge to ``a.b.c`` when that is a module
of the package, else to ``a.b``; a parent package's ``__init__`` is not counted as imported
(it is, by Python, but it declares nothing the child uses).
"""

from __future__ import annotations

import ast
from pathlib import Path

ENGINE = Path(__file__).resolve().parent.parent / "engine"


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
    assert "engine.runtime" in edges and "engine.endpoints.mavlink.connection" in edges
    assert "engine.endpoints.base" in edges["engine.runtime"] or any(
        "engine.endpoints" in target for target in edges["engine.runtime"])
    found = cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}})
    assert found == [["a", "b", "c"]]
    assert a_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}, ["a", "b", "c"]) == ["a", "b", "c", "a"]


def test_function_level_and_type_checking_imports_are_edges(tmp_path: Path):
    source = (
        "from typing import TYPE_CHECKING\n"
        "if TYPE_CHECKING:\n    from engine.runtime import Engine\n"
        "def f():\n    from engine import plan\n    import engine.routes\n"
        "from . import pipeline\n"
    )
    path = tmp_path / "x.py"
    path.write_text(source)
    known = {"engine.runtime", "engine.plan", "engine.routes", "engine.pipeline", "engine.x"}
    assert imports("engine.x", path, known) == {"engine.runtime", "engine.plan", "engine.routes", "engine.pipeline"}


def test_engine_modules_import_without_a_cycle():
    problems = describe(graph())
    assert not problems, "import cycles among engine/ modules:\n" + "\n".join(problems)


if __name__ == "__main__":  # python -m tests.test_import_graph: print the cycles
    print("\n".join(describe(graph())) or "no cycle")
