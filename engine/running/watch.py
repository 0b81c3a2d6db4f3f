"""Watching the routes and schemas directories, and the key files connections read, for
edits, new files, deletions and renames.

The directories are watched rather than the files, so an editor's write-to-temp-then-rename
(the file's inode changes) and files that did not exist at start are both seen. watchfiles
groups a burst of events into one notification, so a save that touches several files
triggers one reload. A schema edit matters as much as a route edit: a route's fingerprint
covers the schemas it validates against. So does a new signing key written over the old
one: a connection's fingerprint covers the contents of its key files, which can live
anywhere, so their directories are watched too (only those files count), and the watch is
set up again whenever a reload names other key files. A schema family's subdirectory
(``schemas/vda5050/``) is watched as the schemas directory is; one created while the engine
runs is watched from the next restart.
"""

from __future__ import annotations

import asyncio
import logging
from pathlib import Path
from typing import Callable, Iterable, Sequence, cast

import watchfiles

log = logging.getLogger("engine.running.watch")
RETRY_S = 1.0
"""Pause before watching again after the watcher itself failed (a directory removed)."""


def _is_route_file(path: Path) -> bool:
    return path.name.endswith((".yaml", ".yml")) and not path.name.startswith(".")


def _is_schema_file(path: Path) -> bool:
    return path.name.endswith(".json") and not path.name.startswith(".")


class _StopOrRewatch:
    """The stop event watchfiles polls while it waits (from its own thread): set when the
    engine stops, or when the key files to watch are no longer those being watched."""

    def __init__(self, stop: asyncio.Event, files: Callable[[], frozenset[Path]], watched: frozenset[Path]) -> None:
        self._stop, self._files, self.watched = stop, files, watched
        self._ended = False

    def is_set(self) -> bool:
        return self._ended or self._stop.is_set() or self._files() != self.watched

    def set(self) -> None:  # watchfiles ends its thread this way when the task is cancelled
        self._ended = True


async def watch_routes(
    routes: Path, changed: Callable[[], object], stop: asyncio.Event, schemas: Path | Sequence[Path] | None = None,
    key_files: Callable[[], Iterable[Path]] | None = None,
) -> None:
    """Call ``changed`` after every change of a route file (or of the one file ``routes``
    names), of a schema file (of any of the ``schemas`` directories), or of one of the files ``key_files()`` names now (absolute
    paths); runs until ``stop`` is set, outliving watcher errors. The task's first step, before
    its first await, sets the watch up (watchfiles' RustNotify adds the inotify watches when it
    is made): the engine starts this task before it says it runs (engine/ops/cli.py)."""
    target = routes.resolve()
    single = target if target.is_file() else None
    routes_dir = target.parent if single else target
    schemas_dirs = [d.resolve() for d in ((schemas,) if isinstance(schemas, Path) else schemas or ())]

    def current_key_files() -> frozenset[Path]:
        return frozenset(key_files()) if key_files is not None else frozenset()

    while not stop.is_set():
        keys = current_key_files()

        def wanted(_change: watchfiles.Change, name: str, keys: frozenset[Path] = keys) -> bool:
            path = Path(name)
            if path in keys:
                return True
            if (path.parent in schemas_dirs or path.parent.parent in schemas_dirs) and _is_schema_file(path):
                return True  # a schema, or one of a family's (schemas/vda5050/order.v2.json)
            if path.parent == routes_dir:
                return path == single if single else _is_route_file(path)
            return False

        families = [d for schemas_dir in schemas_dirs if schemas_dir.is_dir() for d in schemas_dir.iterdir() if d.is_dir()]
        directories = {d for d in {routes_dir, *schemas_dirs, *families, *(k.parent for k in keys)} if d.is_dir()}
        if not directories:  # all gone: wait for one to come back
            await asyncio.sleep(RETRY_S)
            continue
        # watchfiles types stop_event as an anyio/asyncio/trio Event but only calls is_set() and
        # set(), which _StopOrRewatch has (duck-typed, as watchfiles' own thread uses it)
        until = cast(asyncio.Event, _StopOrRewatch(stop, current_key_files, keys))
        try:
            async for _changes in watchfiles.awatch(
                *sorted(directories), watch_filter=wanted, stop_event=until, recursive=False
            ):
                changed()
        except Exception as error:  # a watched directory removed, inotify limits: keep trying
            log.error("watching for changes failed; retrying", extra={"error": f"{type(error).__name__}: {error}"})
        else:
            if not stop.is_set():
                continue  # other key files to watch: watch again at once
        if not stop.is_set():
            await asyncio.sleep(RETRY_S)
            changed()  # whatever happened while not watching
