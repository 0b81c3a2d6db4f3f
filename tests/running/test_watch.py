"""The watcher sees route, schema and key-file edits, and follows the key files a reload names."""

from __future__ import annotations

import asyncio
import time
from pathlib import Path

import pytest

from engine.running.watch import watch_routes

pytestmark = pytest.mark.fast  # no broker, no network peer, no ROS 2 node: ./scripts/test.sh's first tier


async def _seen(calls: list[float], after: int, timeout: float = 10.0) -> bool:
    deadline = time.monotonic() + timeout
    while len(calls) <= after:
        if time.monotonic() > deadline:
            return False
        await asyncio.sleep(0.02)
    return True


def test_key_files_are_watched_and_followed_across_reloads(tmp_path: Path) -> None:
    routes, first, second = tmp_path / "routes", tmp_path / "keys-a", tmp_path / "keys-b"
    for directory in (routes, first, second):
        directory.mkdir()
    (first / "a.key").write_text("old")
    (first / "unrelated.txt").write_text("x")
    keys = {"now": frozenset({(first / "a.key").resolve()})}

    async def scenario() -> None:
        calls: list[float] = []
        stop = asyncio.Event()
        task = asyncio.create_task(watch_routes(routes, lambda: calls.append(time.monotonic()), stop, None, lambda: keys["now"]))
        try:
            await asyncio.sleep(0.3)  # the watch is set up
            (first / "unrelated.txt").write_text("y")
            (first / "a.key").write_text("new")
            assert await _seen(calls, 0), "a key file edit was not seen"
            count = len(calls)
            keys["now"] = frozenset({(second / "b.key").resolve()})  # a reload named another key file
            await asyncio.sleep(0.5)
            (second / "b.key").write_text("new")
            assert await _seen(calls, count), "a key file named by a reload was not watched"
            count = len(calls)
            (routes / "r.yaml").write_text("routes: []\n")
            assert await _seen(calls, count), "a route file edit was not seen"
        finally:
            stop.set()
            await asyncio.wait_for(task, 10)

    asyncio.run(scenario())
