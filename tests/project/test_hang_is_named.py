"""A hung test fails on its own, within its timeout, and the report names it (pytest-timeout,
configured in pyproject.toml), with the xdist workers ./scripts/test.sh uses and without them.

pytest runs in a subprocess on a temporary test file holding a test that passes and three that
hang: in a sleep, on an event no one sets (a lock, as a blocked thread join waits), and in an
asyncio loop. The run must end well inside the bound, each hung test failed by name, the test
beside them passed: one hang no longer spends ./scripts/test.sh's 1500 s and says nothing."""

from __future__ import annotations

import os
import subprocess
import sys
import time
import tomllib
from pathlib import Path

import pytest

from tests.support.repo import REPO

pytestmark = pytest.mark.fast

HUNG = '''
import asyncio
import threading
import time
import tomllib


def test_passes_beside_the_hangs():
    assert True


def test_hangs_in_a_sleep():
    time.sleep(3600)


def test_hangs_on_an_event_no_one_sets():
    threading.Event().wait()


def test_hangs_in_an_event_loop():
    asyncio.run(asyncio.sleep(3600))
'''
TIMEOUT_S = 2
HUNG_TESTS = ("test_hangs_in_a_sleep", "test_hangs_on_an_event_no_one_sets", "test_hangs_in_an_event_loop")


@pytest.mark.parametrize("workers", [[], ["-n", "2"]], ids=["one-process", "xdist"])
def test_a_hung_test_fails_within_its_timeout_and_is_named(tmp_path: Path, workers: list[str]) -> None:
    hung = tmp_path / "test_deliberately_hung.py"
    hung.write_text(HUNG)
    started = time.monotonic()
    # -c: the project's pytest configuration (the timeout method) on a file outside tests/, so
    # tests/conftest.py (its fixtures and tiers) stays out of the run under test.
    result = subprocess.run(
        [sys.executable, "-m", "pytest", "-c", str(REPO / "pyproject.toml"), "--rootdir", str(tmp_path),
         "-p", "no:cacheprovider", "-q", "--timeout", str(TIMEOUT_S), *workers, str(hung)],
        cwd=tmp_path, capture_output=True, text=True, timeout=120,
        env={**os.environ, "COLUMNS": "300"})  # the summary lines whole
    elapsed = time.monotonic() - started
    out = result.stdout + result.stderr
    # Three hangs of TIMEOUT_S each, one after another at worst, plus pytest's (and its workers') start.
    assert elapsed < 3 * TIMEOUT_S + 40, f"took {elapsed:.0f} s:\n{out}"
    assert result.returncode == 1, out
    for name in HUNG_TESTS:
        assert f"FAILED test_deliberately_hung.py::{name} - Failed: Timeout (>{TIMEOUT_S}.0s)" in out, f"{name} not named:\n{out}"
    assert "3 failed, 1 passed" in out, out


def test_every_test_has_a_timeout_by_default() -> None:
    """The bound above is the one every test gets without asking (pyproject.toml)."""
    options = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["pytest"]["ini_options"]
    assert options["timeout"] == 300 and options["timeout_method"] == "signal", options
