"""No unexplained fixed sleep in the tests (issue 30): a test that sleeps a fixed time and hopes
the thing happened meanwhile is slow when the machine is idle and flaky when it is loaded; it waits
on the event or count instead (tests/support/waiting.py ``wait_for``), which goes on the moment it
holds and fails naming what it waited for.

Some sleeps are not waits: a publisher's pace, a quiet window that proves nothing arrives, an
outage's length, a poll interval inside a wait with a deadline, a state the test cannot observe
(a DDS reader matching a writer on the far side). Each of those says so in a comment on the same
line (``# pacing: ...``, ``# quiet window: ...``, ``# outage: ...``, ``# poll: ...``,
``# settle: ...``), so a reviewer sees every fixed sleep and its reason. ``sleep(0)`` (a yield to
the event loop) needs none. A sleep inside a string (a child process's script) is not seen."""

from __future__ import annotations

import ast
import io
import re
import tokenize
from pathlib import Path

import pytest

from tests.support.repo import REPO

pytestmark = pytest.mark.fast

SLEEPERS = ("time", "asyncio")
REASONS = ("pacing", "quiet window", "outage", "poll", "settle")
_REASON = re.compile(r"#\s*(" + "|".join(REASONS) + r"):\s*\S")
"""A comment that names its kind of fixed time and then says why (``# noqa`` or a bare ``#`` is not one)."""


def _explained_lines(source: str) -> set[int]:
    """The lines whose comment gives a reason (a ``#`` inside a string is not a comment)."""
    tokens = tokenize.generate_tokens(io.StringIO(source).readline)
    return {token.start[0] for token in tokens if token.type == tokenize.COMMENT and _REASON.match(token.string)}


def _sleep_names(tree: ast.Module) -> tuple[set[str], set[str]]:
    """``(modules, functions)``: the names ``time``/``asyncio`` are bound to (``import time as t``)
    and the names ``sleep`` itself is bound to (``from asyncio import sleep as nap``)."""
    modules, functions = set(SLEEPERS), set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            modules |= {alias.asname for alias in node.names if alias.name in SLEEPERS and alias.asname}
        elif isinstance(node, ast.ImportFrom) and node.module in SLEEPERS:
            functions |= {alias.asname or alias.name for alias in node.names if alias.name == "sleep"}
    return modules, functions


def _sleep_argument(call: ast.Call, modules: set[str], functions: set[str]) -> ast.expr | None:
    """The duration of a sleep call (positional or ``delay=``/``secs=``), or None if it is no sleep."""
    func = call.func
    is_sleep = ((isinstance(func, ast.Attribute) and func.attr == "sleep" and isinstance(func.value, ast.Name)
                 and func.value.id in modules) or (isinstance(func, ast.Name) and func.id in functions))
    if not is_sleep:
        return None
    if call.args:
        return call.args[0]
    return next((keyword.value for keyword in call.keywords if keyword.arg in ("delay", "secs", "seconds")), None)


def _is_zero(argument: ast.expr) -> bool:
    return isinstance(argument, ast.Constant) and argument.value == 0


def unexplained_sleeps(path: Path) -> list[int]:
    """Lines of ``path`` holding a sleep (``time.sleep``, ``asyncio.sleep``, under any name they
    were imported as) of other than a literal 0 (a number, a name, an expression) with no reason
    on that line."""
    source = path.read_text(encoding="utf-8")
    explained = _explained_lines(source)
    tree = ast.parse(source, str(path))
    modules, functions = _sleep_names(tree)
    lines = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Call) and node.lineno not in explained:
            argument = _sleep_argument(node, modules, functions)
            if argument is not None and not _is_zero(argument):
                lines.append(node.lineno)
    return sorted(lines)


def test_the_scan_sees_a_fixed_sleep(tmp_path: Path):
    sample = tmp_path / "sample.py"
    sample.write_text("import asyncio, time\n"
                      "import time as clock\n"
                      "from asyncio import sleep as nap\n"
                      "time.sleep(0.5)\n"
                      "time.sleep(0)\n"
                      "time.sleep(pause)  # pacing: the publisher's rate\n"
                      "asyncio.sleep(delay)\n"
                      "text = 'time.sleep(1)  # not code'\n"
                      "time.sleep(1)  # noqa\n"
                      "time.sleep(1)  # because\n"
                      "asyncio.sleep(delay=2)\n"
                      "clock.sleep(3)\n"
                      "nap(4)\n"
                      "nap(0.1)  # poll: between two reads\n", encoding="utf-8")
    assert unexplained_sleeps(sample) == [4, 7, 9, 10, 11, 12, 13]


def test_every_fixed_sleep_says_why():
    found = [f"{path.relative_to(REPO).as_posix()}:{line}"
             for path in sorted((REPO / "tests").rglob("*.py")) for line in unexplained_sleeps(path)]
    assert not found, ("fixed sleeps with no reason (wait on the event with tests/support/waiting.py wait_for, or "
                       "say on the same line why it is a fixed time: '# pacing: ...', '# quiet window: ...', "
                       "'# outage: ...', '# poll: ...', '# settle: ...'): " + ", ".join(found))
