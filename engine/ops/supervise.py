"""Running ``run --workers N`` as the command line does: the supervisor (engine/ops/supervisor.py),
its admin (engine/ops/supervisor_admin.py), its Foxglove view (engine/ops/supervisor_foxglove.py),
the watch and the signals, in one place apart from them so that none imports its caller."""

from __future__ import annotations

import argparse
import asyncio
import logging
import signal
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

from engine.common.schemas import SchemaRegistry
from engine.language.route_yaml import Problem
from engine.language.routes import RoutesInvalid, load_routes
from engine.language.specs import RoutesConfig
from engine.ops.admin import AdminAccess
from engine.ops.supervisor import Supervisor
from engine.ops.supervisor_admin import SupervisorAdmin, status_document
from engine.running.placement import PlacementError, place_routes
from engine.running.watch import watch_routes

if TYPE_CHECKING:  # imported when --foxglove asks for it (the SDK's import costs some 40 ms)
    from engine.ops.foxglove import FoxgloveView

log = logging.getLogger("engine.ops.supervise")


def compiler(args: argparse.Namespace, schema_dirs: list[Path],
             vet: Callable[[RoutesConfig, SchemaRegistry], list[Problem]] | None) -> Callable[[], RoutesConfig]:
    """The supervisor's check of the routes: the workers' own (Engine.compile), once for all."""

    def compile_routes() -> RoutesConfig:
        schemas = SchemaRegistry(schema_dirs)
        config = load_routes(args.routes, schemas)
        problems = vet(config, schemas) if vet is not None else []
        try:
            place_routes(config, args.workers)  # a route the workers cannot run (placement rule 1b) reaches none
        except PlacementError as error:
            problems = [*problems, Problem(error.file, error.line, f"{error.message} (with --workers {args.workers})")]
        if problems:
            raise RoutesInvalid(problems, list(config.warnings))
        return config

    return compile_routes


async def foxglove_view(args: argparse.Namespace, supervisor: Supervisor, schema_dirs: list[Path]) -> FoxgloveView | None:
    """``--foxglove`` of the whole engine (engine/ops/supervisor_foxglove.py), started before
    the workers as one engine starts it before its routes (it shows the routes once they run)."""
    from engine.ops.foxglove import start_view
    from engine.ops.supervisor_foxglove import WorkersFeed
    return await start_view(WorkersFeed(supervisor, schema_dirs), args)


async def supervise(args: argparse.Namespace, supervisor: Supervisor, access: AdminAccess | None,
                    write_status: Callable[[dict[str, Any]], None], schema_dirs: list[Path]) -> int:
    """``run --workers N``: start the workers, serve the admin (and the Foxglove view), reload
    on changes and SIGHUP, write the status file, and stop every worker on SIGTERM or SIGINT;
    the exit status as ``run``'s (2: invalid routes, 1: a worker, the admin or the view could
    not start)."""
    view = await foxglove_view(args, supervisor, schema_dirs) if args.foxglove else None
    if args.foxglove and view is None:
        return 1
    try:
        return await _supervise(args, supervisor, access, write_status)
    finally:
        if view is not None:
            await view.stop()


async def _supervise(args: argparse.Namespace, supervisor: Supervisor, access: AdminAccess | None,
                     write_status: Callable[[dict[str, Any]], None]) -> int:
    stopping, reload_requested = asyncio.Event(), asyncio.Event()
    loop = asyncio.get_running_loop()
    for signum in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(signum, stopping.set)
    loop.add_signal_handler(signal.SIGHUP, reload_requested.set)
    admin = SupervisorAdmin(supervisor, args.admin[0], args.admin[1], access) if args.admin else None
    try:
        await supervisor.start()
    except RoutesInvalid as invalid:
        for problem in invalid.problems:
            log.error("invalid routes", extra={"problem": str(problem)})
        return 2
    except RuntimeError as error:
        log.error("cannot start", extra={"error": str(error)})
        return 1
    if admin is not None:
        try:
            await admin.start()
        except OSError as exc:
            log.error("admin endpoint cannot listen", extra={"address": "%s:%s" % args.admin, "error": str(exc)})
            await supervisor.stop(args.drain_timeout)
            return 1

    async def reloader() -> None:
        while True:
            await reload_requested.wait()
            reload_requested.clear()
            await supervisor.reload()

    async def reporter() -> None:
        while True:
            if args.status_file:
                write_status(await status_document(supervisor))
            await asyncio.sleep(args.stats_interval)

    # the watch first, as in ``run`` (engine/ops/cli.py says why)
    tasks = [] if args.no_watch else [
        asyncio.create_task(watch_routes(args.routes, reload_requested.set, stopping, args.schemas or None,
                                         lambda: supervisor.config.watched_files if supervisor.config else frozenset()))]
    tasks += [asyncio.create_task(reloader()), asyncio.create_task(reporter())]
    await stopping.wait()
    log.info("stopping: every worker drains its in-flight messages", extra={"drain_timeout": args.drain_timeout})
    for task in tasks:
        task.cancel()
    await asyncio.gather(*tasks, return_exceptions=True)
    await supervisor.stop(args.drain_timeout)
    if admin is not None:
        await admin.stop()
    if args.status_file:
        write_status(supervisor.status())
    log.info("stopped")
    return 0
