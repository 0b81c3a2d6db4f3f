"""``rabbitros-engine``: run the routes of a directory, check them, or show the live status."""

from __future__ import annotations

import argparse
import asyncio
import logging
import os
import signal
import sys
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING, Any, Sequence

import orjson

from engine import __version__
from engine.common.json_bytes import json_bytes
from engine.common.logs import setup_logging
from engine.common.processes import LOCAL_BROKER_ENV, BrokerError, PrivateBroker
from engine.common.redaction import redact_urls
from engine.common.schemas import SchemaRegistry
from engine.endpoints.base import EndpointError
from engine.language.routes import RoutesInvalid, load_routes
from engine.ops.admin import AdminAccess, AdminConfigError, AdminServer, admin_access, status_document
from engine.ops.dead_letter_tool import run_command as run_dead_letters
from engine.ops.dead_letter_tool import selection_of
from engine.ops.cli_parser import COMMANDS, build_parser
from engine.ops.local_broker import private_brokers, stand_in_for_check
from engine.ops.opsview import AdminClient, print_status, print_tap
from engine.ops.replay import run_from_recording, run_replay
from engine.ops.replay_sinks import run_replay_to_sinks
from engine.ops.route_tests import failing_tests, format_result, load_checked, run_tests
from engine.ops.supervise import compiler, supervise
from engine.ops.supervisor import Supervisor
from engine.running.loop import LoopChoiceError, loop_factory
from engine.running.loop import run as run_loop
from engine.running.observe import COUNTERS
from engine.running.record import Recorder, RecordLimits
from engine.running.runtime import Engine
from engine.running.placement import PlacementError, place_routes
from engine.running.watch import watch_routes
from engine.running.worker import WorkerEngine, die_with_parent, log_as_worker, tell_supervisor

if TYPE_CHECKING:  # imported when --foxglove asks for it: the SDK's import costs some 40 ms every command would pay
    from engine.ops.foxglove import FoxgloveView

log = logging.getLogger("engine.ops.cli")


def default_schemas(routes: Path) -> Path:
    """``schemas/`` beside the routes directory (or above it), else the working directory's."""
    base = routes.parent if routes.is_file() else routes
    for candidate in (base / "schemas", base.parent / "schemas", Path("schemas")):
        if candidate.is_dir():
            return candidate
    return Path("schemas")


def schema_directories(args: argparse.Namespace) -> list[Path]:
    """Every ``--schemas`` given, in order (a later one over the earlier), else the default."""
    return list(args.schemas) if args.schemas else [default_schemas(args.routes)]

def _client(args: argparse.Namespace) -> AdminClient | int:
    try:
        return AdminClient.from_files(args.admin, args.admin_token_file, args.admin_ca_file)
    except AdminConfigError as exc:
        print(exc, file=sys.stderr)
        return 2


def main(argv: Sequence[str] | None = None) -> int:
    args_list = list(sys.argv[1:] if argv is None else argv)
    if not any(arg in COMMANDS or arg in ("-h", "--help", "--version") for arg in args_list[:1]):
        args_list.insert(0, "run")
    args = build_parser().parse_args(args_list)
    if args.command == "check":
        if args.local_broker:  # the private brokers' URLs are not known before they start: stand-ins no route file names
            stand_in_for_check()
        return check(args.routes, schema_directories(args), args.workers)
    if args.command == "test" and args.from_recording:
        if not args.route:
            print("test --from-recording needs --route NAME", file=sys.stderr)
            return 2
        return run_from_recording(args.from_recording, args.routes, schema_directories(args), args.route, args.count)
    if args.command == "test":
        return run_route_tests(args.routes, schema_directories(args))
    if args.command == "replay" and args.to_sinks:
        return run_replay_to_sinks(args.recording, args.routes, schema_directories(args), args.route, args.speed)
    if args.command == "replay":
        return run_replay(args.recording, args.routes, schema_directories(args), args.route, tuple(args.ignore))
    if args.command == "status":
        if args.admin:
            client = _client(args)
            return client if isinstance(client, int) else print_status(args.admin, args.json, client)
        try:
            print(args.status_file.read_text(), end="")
        except OSError as exc:
            print(f"{args.status_file}: {exc.strerror}", file=sys.stderr)
            return 1
        return 0
    if args.command == "dead-letters":
        try:
            selection = selection_of(args.route, args.stage, args.id, args.since, args.until)
        except ValueError as exc:
            print(exc, file=sys.stderr)
            return 2
        logging.basicConfig(level=logging.WARNING, format="%(message)s")
        return run_dead_letters(args.action, args.routes, args.schemas or default_schemas(args.routes), selection,
                                args.limit, getattr(args, "ready_timeout", 10.0))
    if args.command == "tap":
        client = _client(args)
        return client if isinstance(client, int) else print_tap(args.admin, args.route, args.count, client)
    listener = setup_logging(args.log_level, args.log_format)
    try:
        loop_factory()  # a loop it cannot run is refused by name before anything starts
    except LoopChoiceError as error:
        listener.stop()
        print(f"error: {error}", file=sys.stderr)
        return 2
    try:
        return run_loop(run(args))
    finally:
        # Stopped: a second SIGTERM must not kill the exit itself (-15 instead of 0) once the
        # loop, whose handler took the first, has put back the default action. It comes: GNU
        # ``timeout`` (as systemd's KillMode=mixed, a supervisor asking twice) passes the signal
        # it got on to its process group, which the engine already got from ``kill -- -PGID``.
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        listener.stop()


def check(routes: Path, schema_dirs: Path | Sequence[Path], workers: int = 1) -> int:
    schema_dirs = [schema_dirs] if isinstance(schema_dirs, Path) else list(schema_dirs)
    try:
        registry = SchemaRegistry(schema_dirs)
        config, cases, problems, warnings = load_checked(routes, registry)
    except Exception as error:  # what the loader did not foresee still gets one line, not a traceback
        print(f"{routes}: cannot load: {type(error).__name__}: {error}", file=sys.stderr)
        return 1
    shown = [(p.file, p.line, str(p)) for p in problems] + [(w.file, w.line, f"{w.file}:{w.line}: warning: {w.message}") for w in warnings]
    for _, _, line in sorted(shown):  # every problem and warning of the run, in file order
        print(line, file=sys.stderr)
    if config is None or problems:
        return 1
    tests = f", {len(cases)} tests" if cases else ""
    print(f"{routes}: {len(config.routes)} routes, {len(config.connections)} connections{tests}, config {config.content_hash}: ok")
    if len(schema_dirs) > 1:  # several directories: which file each schema the routes use came from
        for schema_file in registry.files_used(sorted({route.schema for route in config.routes.values()})):
            over = f" (over {', '.join(map(str, schema_file.replaces))})" if schema_file.replaces else ""
            print(f"  schema {schema_file.relative}: {schema_file.path}{over}")
    if workers > 1:
        try:
            print("\n".join(place_routes(config, workers).lines()))
        except PlacementError as error:
            print(f"{error} (with --workers {workers})", file=sys.stderr)
            return 1
    return 0


def run_route_tests(routes: Path, schema_dirs: Path | Sequence[Path]) -> int:
    """``rabbitros-engine test``: one line per case, a diff per failure; 0 pass, 1 fail, 2 invalid."""
    schemas = SchemaRegistry(schema_dirs)
    config, cases, problems, _ = load_checked(routes, schemas)
    for problem in problems:
        print(problem, file=sys.stderr)
    if config is None or problems:
        return 2
    if not cases:
        print(f"{routes}: no tests (add *.test.yaml files beside the routes)", file=sys.stderr)
        return 2
    failed = 0
    for result in run_tests(cases, config, schemas):
        failed += not result.passed
        print("\n".join(format_result(result)), flush=True)
    print(f"{len(cases) - failed} passed, {failed} failed")
    return 1 if failed else 0


async def run(args: argparse.Namespace) -> int:
    started: list[PrivateBroker] = []
    access = None
    if args.admin:
        try:
            access = admin_access(args.admin[0], args.admin_token_file, args.admin_tls_cert, args.admin_tls_key)
        except AdminConfigError as exc:
            log.error("admin endpoint refused", extra={"error": str(exc)})
            return 2
    if args.cluster < 1 or (args.cluster > 1 and not args.local_broker):
        log.error("--cluster N needs --local-broker and N >= 1")
        return 2
    if args.local_broker_tls and not args.local_broker:
        log.error("--local-broker-tls needs --local-broker")
        return 2
    try:
        if args.local_broker:
            try:
                brokers = private_brokers(args.cluster, _protocols_used(args), tls=args.local_broker_tls)
            except BrokerError as exc:
                log.error("local broker refused", extra={"error": str(exc)})
                return 2
            for broker in brokers:
                try:
                    await asyncio.to_thread(broker.start)
                except BrokerError as exc:
                    log.error("local broker failed to start", extra={"error": str(exc)})
                    return 1
                started.append(broker)
                os.environ.update(broker.environment)
            urls = [url for broker in started for url in broker.urls]
            nodes = [node for broker in started for node in broker.nodes]
            os.environ[LOCAL_BROKER_ENV] = ", ".join(nodes)  # the loader warns about connections that go elsewhere
            environment = {key: redact_urls(value) for broker in started for key, value in broker.environment.items()}
            log.info("local broker started", extra={"urls": [redact_urls(u) for u in urls], "nodes": nodes, "environment": environment})
            if args.broker_url_file:
                _write_atomically(args.broker_url_file, "\n".join(urls) + "\n")
        return await serve(args, access)
    finally:
        for broker in reversed(started):
            await asyncio.to_thread(broker.stop)


def _protocols_used(args: argparse.Namespace) -> set[str] | None:
    """The protocols of the routes' connections (each protocol's private broker starts only
    when used, unless it always does); None when the routes do not load (every broker)."""
    saved = dict(os.environ)
    try:
        stand_in_for_check()
        config = load_routes(args.routes, SchemaRegistry(schema_directories(args)))
    except (RoutesInvalid, OSError, EndpointError):
        return None
    finally:
        os.environ.clear()
        os.environ.update(saved)
    return {connection.protocol for connection in config.connections.values()}


async def serve(args: argparse.Namespace, access: AdminAccess | None = None) -> int:
    if getattr(args, "workers", 1) > 1 and getattr(args, "worker", None) is None:
        supervisor = Supervisor(args, args.workers, compiler(args, schema_directories(args), failing_tests if args.test_on_reload else None),
                                access.token if access is not None else None)
        return await supervise(args, supervisor, access, lambda document: _write_status(args.status_file, document),
                               schema_directories(args))
    recorder = None if args.record is None else Recorder(args.record, RecordLimits(
        file_bytes=int(args.record_file_mb * 2**20), file_seconds=args.record_file_minutes * 60,
        total_bytes=int(args.record_total_mb * 2**20)))
    worker = {"index": args.worker, "workers": args.workers, "runtime_dir": args.runtime_dir} \
        if getattr(args, "worker", None) is not None else None
    if worker is not None:
        die_with_parent(args.supervisor_pid)
        log_as_worker(args.worker)
    engine = (WorkerEngine if worker is not None else Engine)(
        args.routes, schema_directories(args), require_connections=args.require_connections, instance=args.instance,
        vet=failing_tests if args.test_on_reload else None, recorder=recorder, **(worker or {}))
    admin = AdminServer(engine, args.admin[0], args.admin[1], access) if args.admin else None
    if admin is not None:
        try:
            await admin.start()
        except OSError as exc:
            log.error("admin endpoint cannot listen", extra={"address": "%s:%s" % args.admin, "error": str(exc)})
            return 1
        args.admin_bound_port = admin.port
    view = await _foxglove_view(args, engine)
    if view == 1:
        return 1
    try:
        if recorder is not None:
            try:
                recorder.start()
            except OSError as exc:
                log.error("cannot record", extra={"directory": str(args.record), "error": str(exc)})
                return 2
        return await _serve(args, engine)
    finally:
        if view is not None and not isinstance(view, int):
            await view.stop()
        if admin is not None:
            await admin.stop()
        if recorder is not None:  # after the routes stopped: what they sent last is in the file, which gets its summary
            await asyncio.to_thread(recorder.stop)


async def _foxglove_view(args: argparse.Namespace, engine: Engine) -> FoxgloveView | int | None:
    """``--foxglove``: the view started (it follows the routes once they run), 1 when it
    cannot be, None when not asked for."""
    if not getattr(args, "foxglove", None):
        return None
    from engine.ops.foxglove import EngineFeed, start_view
    view = await start_view(EngineFeed(engine), args)
    return 1 if view is None else view


async def _serve(args: argparse.Namespace, engine: Engine) -> int:
    stopping = asyncio.Event()
    loop = asyncio.get_running_loop()
    loop.add_signal_handler(signal.SIGINT, stopping.set)
    loop.add_signal_handler(signal.SIGTERM, stopping.set)
    try:
        await engine.start()
    except RoutesInvalid as invalid:
        for problem in invalid.problems:
            log.error("invalid routes", extra={"problem": str(problem)})
        return 2
    except EndpointError as error:
        log.error("cannot start", extra={"error": str(error)})
        await engine.stop(0.0)
        return 1

    reload_requested = asyncio.Event()
    loop.add_signal_handler(signal.SIGHUP, reload_requested.set)

    async def reloader() -> None:
        while True:
            await reload_requested.wait()
            reload_requested.clear()
            try:
                await engine.reload()
            except Exception:  # Engine.reload rejects what it can foresee; this loop must outlive the rest
                log.exception("reload failed")
            write_status()

    def write_status() -> None:
        if args.status_file is not None:
            _write_status(args.status_file, status_document(engine))

    async def reporter() -> None:
        while True:
            engine.observers.sample()
            write_status()
            await asyncio.sleep(args.stats_interval)
            if log.isEnabledFor(logging.INFO):  # the status of 200 routes is ~10 ms of the loop: not for a line nobody keeps
                for name, route in engine.status()["routes"].items():
                    log.info("route counters", extra={"route": name, **{k: route[k] for k in (*COUNTERS, "dead_lettered")}})

    # The watch first: its task's first step sets up inotify (watchfiles' RustNotify, before its
    # first await), and it runs before the reporter's first step writes the status that says the
    # engine runs. Created after it, an edit made as soon as the status said so went unseen (a
    # test missed its reload for 30 s beside a busy CI).
    tasks = [] if args.no_watch else [
        asyncio.create_task(watch_routes(args.routes, reload_requested.set, stopping, engine.schemas_dirs, engine.key_files))]
    tasks += [asyncio.create_task(reloader()), asyncio.create_task(reporter())]
    log.info("engine running", extra={"routes": len(engine.runners), "generation": engine.generation, "version": __version__, "instance": engine.instance})
    if getattr(args, "worker_channel", None) is not None:  # a worker: tell the supervisor where its admin answers
        tell_supervisor(args.worker_channel, {"admin_port": getattr(args, "admin_bound_port", None), "pid": os.getpid()})
    await stopping.wait()
    log.info("stopping: draining in-flight messages", extra={"drain_timeout": args.drain_timeout})
    for task in tasks:
        task.cancel()
    await asyncio.gather(*tasks, return_exceptions=True)
    await engine.stop(args.drain_timeout)
    write_status()
    log.info("stopped")
    return 0


STATUS_JSON = orjson.OPT_INDENT_2 | orjson.OPT_NON_STR_KEYS | orjson.OPT_APPEND_NEWLINE
"""The status file's encoding: orjson, in C. ``json.dumps(indent=2)`` runs the standard
library's pure-Python encoder (``indent`` turns its C encoder off): with the fleet benchmark's
200 routes it held the loop ~20 ms every second (py-spy, bench/fleet.py), a stall every message
arriving meanwhile waited out, and the largest part of one engine's p99 there."""


def _write_status(path: Path | None, document: dict[str, Any]) -> None:
    if path is not None:  # json_bytes: a value orjson refuses must not end the reporter (engine/common/json_bytes.py)
        _write_atomically(path, json_bytes(document, STATUS_JSON))


def _write_atomically(path: Path, data: str | bytes) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.NamedTemporaryFile("wb", dir=path.parent, prefix=f".{path.name}.", delete=False) as tmp:
        tmp.write(data.encode() if isinstance(data, str) else data)
    os.replace(tmp.name, path)
