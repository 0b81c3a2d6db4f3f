"""Watching the routes and schemas directories for edits, new files, deletions and renames.

The directories are watched rather than the files, so an editor's write-to-temp-then-rename
(the file's inode changes) and files that did not exist at start are both seen. watchfiles
groups a burst of events into one notification, so a save that touches several files
triggers one reload. A schema edit matters as much as a route edit: a route's fingerprint
covers the schemas it validates against.
"""

from __future__ import annotations

import asyncio
import logging
from pathlib import Path
from typing import Callable

import watchfiles

log = logging.getLogger("engine.watch")
RETRY_S = 1.0
"""Pause before watching again after the watcher itself failed (a directory removed)."""


def _is_route_file(path: Path) -> bool:
    return path.name.endswith((".yaml", ".yml")) and not path.name.startswith(".")


def _is_schema_file(path: Path) -> bool:
    return path.name.endswith(".json") and not path.name.startswith(".")


async def watch_routes(
    routes: Path, changed: Callable[[], None], stop: asyncio.Event, schemas: Path | None = None
) -> None:
    """Call ``changed`` after every change of a route file (or of the one file ``routes``
    names) or of a schema file; runs until ``stop`` is set, outliving watcher errors."""
    target = routes.resolve()
    single = target if target.is_file() else None
    routes_dir = target.parent if single else target
    schemas_dir = schemas.resolve() if schemas is not None else None

    def wanted(_change: watchfiles.Change, name: str) -> bool:
        path = Path(name)
        if schemas_dir is not None and path.parent == schemas_dir and _is_schema_file(path):
            return True
        if path.parent == routes_dir:
            return path == single if single else _is_route_file(path)
        return False

    while not stop.is_set():
        directories = [d for d in {routes_dir, schemas_dir} if d is not None and d.is_dir()]
        if not directories:  # both gone: wait for one to come back
            await asyncio.sleep(RETRY_S)
            continue
        try:
            async for _changes in watchfiles.awatch(
                *directories, watch_filter=wanted, stop_event=stop, recursive=False
            ):
                changed()
        except Exception as error:  # a watched directory removed, inotify limits: keep trying
            log.error("watching for changes failed; retrying", extra={"error": f"{type(error).__name__}: {error}"})
        if not stop.is_set():
            await asyncio.sleep(RETRY_S)
            changed()  # whatever happened while not watching
