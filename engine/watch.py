"""Watching the routes directory for edits, new files, deletions and atomic renames.

The parent directory is watched rather than the files, so an editor's write-to-temp-then-
rename (the file's inode changes) and files that did not exist at start are both seen.
watchfiles groups a burst of events (debounce) into one notification, so a save that
touches several files triggers one reload.
"""

from __future__ import annotations

import asyncio
from pathlib import Path
from typing import Callable

import watchfiles


def _is_route_file(path: str) -> bool:
    name = Path(path).name
    return name.endswith((".yaml", ".yml")) and not name.startswith(".")


async def watch_routes(routes: Path, changed: Callable[[], None], stop: asyncio.Event) -> None:
    target = routes.resolve()
    directory = target.parent if target.is_file() else target
    single = target if target.is_file() else None

    def wanted(_change: watchfiles.Change, path: str) -> bool:
        return Path(path) == single if single else _is_route_file(path)

    async for _changes in watchfiles.awatch(directory, watch_filter=wanted, stop_event=stop, recursive=False):
        changed()

