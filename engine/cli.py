"""``rabbitros-engine``: run the routes of a directory, check them, or show the live status."""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import os
import signal
import sys
import tempfile
from pathlib import Path
from typing import Sequence

from engine import __version__
from engine.endpoints.amqp import redact
from engine.endpoints.base import EndpointError
from engine.local_broker import BrokerError, LocalBroker
from engine.logs import setup_logging
from engine.loop import run as run_loop
from engine.routes import RoutesInvalid, load_routes
from engine.runtime import Engine
from engine.schemas import SchemaRegistry
from engine.watch import watch_routes

log = logging.getLogger("engine.cli")
COMMANDS = ("run", "check", "status")


def default_schemas(routes: Path) -> Path:
    """``schemas/`` beside the routes directory (or above it), else the working directory's."""
    base = routes.parent if routes.is_file() else routes
    for candidate in (base / "schemas", base.parent / "schemas", Path("schemas")):
        if candidate.is_dir():
            return candidate
    return Path("schemas")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="rabbitros-engine",
        description="Routes messages between RabbitMQ, ROS 2 and MAVLink as declared in YAML route files.",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    commands = parser.add_subparsers(dest="command", metavar="{run,check,status}")

    def common(sub: argparse.ArgumentParser) -> None:
        sub.add_argument("--routes", type=Path, default=Path("routes"), help="routes directory (or one file); default ./routes")
        sub.add_argument("--schemas", type=Path, help="canonical schemas directory; default: schemas/ beside the routes")

    run = commands.add_parser("run", help="run the routes (the default command)")
    common(run)
    run.add_argument("--local-broker", action="store_true", help="start a private RabbitMQ node and use it as the default AMQP connection")
    run.add_argument("--broker-url-file", type=Path, help="with --local-broker: write the broker's URL to this file")
    run.add_argument("--status-file", type=Path, help="keep the live status (generation, config hash, counters) in this JSON file")
    run.add_argument("--no-watch", action="store_true", help="do not reload when route files change (SIGHUP still reloads)")
    run.add_argument("--stats-interval", type=float, default=10.0, help="seconds between status updates and counter logs")
    run.add_argument("--log-level", default="info", choices=["debug", "info", "warning", "error"])
    run.add_argument("--log-format", default="text", choices=["text", "json"])

    check = commands.add_parser("check", help="validate the routes without connecting; exit 0 when valid")
    common(check)

    status = commands.add_parser("status", help="print the live status written by a running engine")
    status.add_argument("--status-file", type=Path, required=True)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args_list = list(sys.argv[1:] if argv is None else argv)
    if not any(arg in COMMANDS or arg in ("-h", "--help", "--version") for arg in args_list[:1]):
        args_list.insert(0, "run")
    args = build_parser().parse_args(args_list)
    if args.command == "check":
        return check(args.routes, args.schemas or default_schemas(args.routes))
    if args.command == "status":
        try:
            print(args.status_file.read_text(), end="")
        except OSError as exc:
            print(f"{args.status_file}: {exc.strerror}", file=sys.stderr)
            return 1
        return 0
    listener = setup_logging(args.log_level, args.log_format)
    try:
        return run_loop(run(args))
    finally:
        listener.stop()


def check(routes: Path, schemas: Path) -> int:
    try:
        config = load_routes(routes, SchemaRegistry(schemas))
    except RoutesInvalid as invalid:
        for problem in invalid.problems:
            print(problem, file=sys.stderr)
        return 1
    print(f"{routes}: {len(config.routes)} routes, {len(config.connections)} connections, config {config.content_hash}: ok")
    return 0


async def run(args: argparse.Namespace) -> int:
    broker: LocalBroker | None = None
    if args.local_broker:
        broker = LocalBroker()
        try:
            url = await asyncio.to_thread(broker.start)
        except BrokerError as exc:
            log.error("local broker failed to start", extra={"error": str(exc)})
            return 1
        os.environ["RABBITROS_AMQP_URL"] = url
        log.info("local broker started", extra={"url": redact(url), "node": broker.node})
        if args.broker_url_file:
            _write_atomically(args.broker_url_file, url + "\n")
    try:
        return await serve(args)
    finally:
        if broker is not None:
            await asyncio.to_thread(broker.stop)


async def serve(args: argparse.Namespace) -> int:
    engine = Engine(args.routes, args.schemas or default_schemas(args.routes))
    try:
        await engine.start()
    except RoutesInvalid as invalid:
        for problem in invalid.problems:
            log.error("invalid routes", extra={"problem": str(problem)})
        return 2
    except EndpointError as error:
        log.error("cannot start", extra={"error": str(error)})
        await engine.stop()
        return 1

    stopping = asyncio.Event()
    reload_requested = asyncio.Event()
    loop = asyncio.get_running_loop()
    loop.add_signal_handler(signal.SIGINT, stopping.set)
    loop.add_signal_handler(signal.SIGTERM, stopping.set)
    loop.add_signal_handler(signal.SIGHUP, reload_requested.set)

    async def reloader() -> None:
        while True:
            await reload_requested.wait()
            reload_requested.clear()
            await engine.reload()
            write_status()

    def write_status() -> None:
        if args.status_file:
            _write_atomically(args.status_file, json.dumps(engine.status(), indent=2) + "\n")

    async def reporter() -> None:
        while True:
            write_status()
            await asyncio.sleep(args.stats_interval)
            for name, route in engine.status()["routes"].items():
                log.info("route counters", extra={"route": name, **{k: route[k] for k in ("received", "delivered", "failed", "sink_errors")}})

    tasks = [asyncio.create_task(reloader()), asyncio.create_task(reporter())]
    if not args.no_watch:
        tasks.append(asyncio.create_task(watch_routes(args.routes, reload_requested.set, stopping)))
    log.info("engine running", extra={"routes": len(engine.runners), "generation": engine.generation, "version": __version__})
    await stopping.wait()
    log.info("stopping: draining in-flight messages")
    for task in tasks:
        task.cancel()
    await asyncio.gather(*tasks, return_exceptions=True)
    await engine.stop()
    write_status()
    return 0


def _write_atomically(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.NamedTemporaryFile("w", dir=path.parent, prefix=f".{path.name}.", delete=False) as tmp:
        tmp.write(text)
    os.replace(tmp.name, path)
