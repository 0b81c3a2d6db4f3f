"""The watcher sees route, schema and key-file edits, and follows the key files a reload names."""

from __future__ import annotations

import asyncio
import time
from pathlib import Path

import pytest

from engine.running.watch import watch_routes
from tests.support.waiting import probe_until, wait_for

pytestmark = pytest.mark.fast  # no broker, no network peer, no ROS 2 node: ./scripts/test.sh's first tier


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
            await asyncio.sleep(0)  # the watch task's first step sets the watch up (engine/running/watch.py), before our next
            (first / "unrelated.txt").write_text("y")
            (first / "a.key").write_text("new")
            await wait_for(lambda: len(calls) > 0, 10, "a key file edit to be seen")
            count = len(calls)
            keys["now"] = frozenset({(second / "b.key").resolve()})  # a reload named another key file
            # the watcher takes the new key set on its next turn and says nothing then: edit until seen
            await probe_until(lambda: len(calls) > count, lambda: (second / "b.key").write_text("new"), 10,
                              "an edit of the key file a reload named to be seen", every=0.25)
            # the probe may have written b.key once more while the watcher reported the last one:
            # that second report must be in before the count the route-file edit is judged by
            await asyncio.sleep(0.4)  # quiet window: longer than the probe's 0.25 s and watchfiles' 50 ms step
            count = len(calls)
            (routes / "r.yaml").write_text("routes: []\n")
            await wait_for(lambda: len(calls) > count, 10, "a route file edit to be seen")
        finally:
            stop.set()
            await asyncio.wait_for(task, 10)

    asyncio.run(scenario())
