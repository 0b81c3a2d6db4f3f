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
import tokenize
from pathlib import Path

import pytest

from tests.support.repo import REPO

pytestmark = pytest.mark.fast

SLEEPERS = ("time", "asyncio")


def _commented_lines(source: str) -> set[int]:
    """The lines that carry a ``#`` comment (a ``#`` inside a string is not one)."""
    tokens = tokenize.generate_tokens(io.StringIO(source).readline)
    return {token.start[0] for token in tokens if token.type == tokenize.COMMENT}


def _is_zero(argument: ast.expr) -> bool:
    return isinstance(argument, ast.Constant) and argument.value == 0


def unexplained_sleeps(path: Path) -> list[int]:
    """Lines of ``path`` holding ``time.sleep(x)`` / ``asyncio.sleep(x)`` with ``x`` other than a
    literal 0 (a number, a name, an expression) and no comment on that line."""
    source = path.read_text(encoding="utf-8")
    commented = _commented_lines(source)
    lines = []
    for node in ast.walk(ast.parse(source, str(path))):
        if (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "sleep"
                and isinstance(node.func.value, ast.Name) and node.func.value.id in SLEEPERS
                and node.args and not _is_zero(node.args[0]) and node.lineno not in commented):
            lines.append(node.lineno)
    return sorted(lines)


def test_the_scan_sees_a_fixed_sleep(tmp_path: Path):
    sample = tmp_path / "sample.py"
    sample.write_text("import asyncio, time\n"
                      "time.sleep(0.5)\n"
                      "time.sleep(0)\n"
                      "time.sleep(pause)  # pacing: the publisher's rate\n"
                      "asyncio.sleep(delay)\n"
                      "text = 'time.sleep(1)  # not code'\n", encoding="utf-8")
    assert unexplained_sleeps(sample) == [2, 5]


def test_every_fixed_sleep_says_why():
    found = [f"{path.relative_to(REPO).as_posix()}:{line}"
             for path in sorted((REPO / "tests").rglob("*.py")) for line in unexplained_sleeps(path)]
    assert not found, ("fixed sleeps with no reason (wait on the event with tests/support/waiting.py wait_for, or "
                       "say on the same line why it is a fixed time: '# pacing: ...', '# quiet window: ...', "
                       "'# outage: ...'): " + ", ".join(found))
